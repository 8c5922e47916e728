"""The host transports against the emulated drives on each attachment: virtual CAN, a slcan pty, an RS485 pty.

The other bus tests pair the emulator with the raw codec, or the transports with scripted peers; here the two meet:
every request command goes through ``Transport.transact`` to emulated drives, the emulator's fault kinds are seen
through the transport's matching and counters, and protocol-breaking input sent to the emulator is counted, logged
and left unanswered. Faults are scheduled in simulation seconds; the attachment keeps simulation time on the
monotonic clock, so a test waits for ``emulator.time_s`` to pass a fault's start or end before it acts on it.

Deadlines are generous and timing is only ever a lower bound (the transport cannot return before the deadline of a
reply that never comes), so that a loaded machine slows these tests down without failing them.
"""

from __future__ import annotations

import dataclasses
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import serial

from motion.emulator import (
    Attachment,
    Corruption,
    DriveModel,
    EmulatedDrive,
    Emulator,
    Fault,
    FrameLog,
    InjectedFault,
    Rs485Attachment,
    RunState,
    Setpoint,
    SlcanAttachment,
    VirtualCanAttachment,
)
from motion.emulator.drive import DriveLoop
from motion.errors import EncodeError
from motion.protocol import (
    COMMANDS,
    Acceleration,
    Bare,
    CanFrame,
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
    ProductInfo,
    Rs485Frame,
    SingleTurnAngle,
    SingleTurnPosition,
    SingleTurnPositionSpeed,
    SpeedControl,
    SpinDirection,
    Status1,
    TorqueControl,
    WireProtocol,
    rs485_frame,
)
from motion.protocol.table import command_of
from motion.transport import CanTransport, Reply, Request, Rs485Transport, Transport
from motion.transport.can_endpoint import CanEndpoint
from tests.test_emulator_drive import check_reply

ATTACHMENTS = ("virtual", "slcan", "rs485")
MOTORS = (1, 2, 3, 4)
#: Deadline of a cycle per request in it, s: generous, a prompt reply takes well under a millisecond.
DEADLINE_S = 0.1
#: How long the line must stay quiet to count as "not answered", s (a prompt reply takes a millisecond or two).
QUIET_S = 0.05
#: Longest wait for the emulator (simulation time, a motion, a cooling drive), s.
WAIT_S = 3.0
#: Distinct names, so that 0x12 is seen to report the model's and not a constant; a short thermal time constant,
#: so that an over-temperature drive cools below its threshold within a fraction of a second after the fault.
MODEL = DriveModel(driver_name="RMD-X8-EMU", motor_name="X8-PRO-TEST", hardware_version=2.1, firmware_version=3.4,
                   thermal_time_constant_s=1.0)  # fmt: skip


def state_of(drive: EmulatedDrive) -> RunState:
    """The drive's run state, read afresh (the attachment's thread and the requests change it)."""
    return drive.state


def setpoint_of(drive: EmulatedDrive) -> Setpoint | None:
    """The drive's last control command, read afresh."""
    return drive.setpoint


def decode_errors_reach(bus: Bus, count: int) -> Callable[[], bool]:
    return lambda: bus.attachment.stats.decode_errors >= count


def wait_for(condition: Callable[[], bool], timeout_s: float = WAIT_S) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.002)
    return True


@dataclass
class Bus:
    """Emulated drives on one attachment, and the host transport that talks to them."""

    kind: str
    emulator: Emulator
    attachment: Attachment[Any, Any]
    log_path: Path
    transport: Transport = field(init=False)
    exercised: set[Command] = field(default_factory=set)

    @property
    def protocol(self) -> WireProtocol:
        return WireProtocol.RS485 if self.kind == "rs485" else WireProtocol.CAN

    def open_transport(self) -> Transport:
        """Open a new host transport on the attachment (the previous one must be closed)."""
        path = self.attachment.path
        if self.kind == "virtual":
            self.transport = CanTransport("virtual", path)
        elif self.kind == "slcan":
            # sleep_after_open: python-can otherwise waits 2 s for a real adapter to boot.
            self.transport = CanTransport("slcan", path, bitrate=1_000_000, sleep_after_open=0)
        else:
            self.transport = Rs485Transport(path)
        return self.transport

    def close_transport(self) -> None:
        self.transport.close()

    def cycle(self, requests: list[Request], budget_s: float | None = None) -> list[Reply]:
        """One ``transact`` with a deadline of ``budget_s`` (default: DEADLINE_S per request) from now."""
        budget = DEADLINE_S * len(requests) if budget_s is None else budget_s
        return self.transport.transact(requests, self.transport.clock() + budget)

    def ask(self, motor_id: int, message: Message) -> Message:
        """One request, answered in time by its drive with the reply the command table declares."""
        (reply,) = self.cycle([Request(motor_id, message)])
        assert reply.motor_id == motor_id and reply.request == message
        assert reply.message is not None, f"motor {motor_id}: no reply to {message}"
        check_reply(message, reply.message, self.protocol)
        command = command_of(message)
        assert command is not None
        self.exercised.add(command)
        return reply.message

    def wait_sim(self, time_s: float) -> None:
        """Wait until simulation time reaches ``time_s``."""
        assert wait_for(lambda: self.emulator.time_s >= time_s), f"simulation time stuck at {self.emulator.time_s}"

    def fault(
        self, kind: InjectedFault, motor_id: int, lasting_s: float | None = None, after_s: float = 0.0, **kwargs: Any
    ) -> Fault:
        """Schedule a fault ``after_s`` s of simulation time from now, ``lasting_s`` long (None: open-ended).

        Returns once simulation time has reached the fault's start.
        """
        start = self.emulator.time_s + after_s
        fault = Fault(kind, motor_id, start, None if lasting_s is None else start + lasting_s, **kwargs)
        self.emulator.add_fault(fault)
        self.wait_sim(start)
        return fault

    def log(self, direction: str) -> list[str]:
        """The wire column of the frame-log lines of ``direction`` (IN, OUT, BAD, NOTE)."""
        wires = []
        for line in self.log_path.read_text().splitlines():
            columns = line.split(maxsplit=3)
            if columns[1] == direction:
                wires.append(columns[3].split(" | ")[0])
        return wires


@pytest.fixture(params=ATTACHMENTS)
def bus(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Bus]:
    kind: str = request.param
    emulator = Emulator(MOTORS, model=MODEL)
    log_path = tmp_path / "frames.log"
    with ExitStack() as stack:
        log = stack.enter_context(FrameLog(log_path))
        attachment: Attachment[Any, Any]
        if kind == "virtual":
            attachment = VirtualCanAttachment(emulator, f"rmd-it-{uuid.uuid4().hex}", frame_log=log)
        elif kind == "slcan":
            attachment = SlcanAttachment(emulator, tmp_path / "slcan", frame_log=log)
        else:
            attachment = Rs485Attachment(emulator, tmp_path / "rs485", frame_log=log)
        # close() re-raises what stopped the attachment's thread, so that an emulator failure fails the test.
        stack.enter_context(attachment)
        rig = Bus(kind, emulator, attachment, log_path)
        rig.open_transport()
        stack.callback(rig.close_transport)  # before the attachment: slcan closes its channel with C
        yield rig


def assert_clean(bus: Bus, motors: tuple[int, ...] = MOTORS) -> None:
    """Every request was answered and matched; nothing late, corrupt, stale or foreign on the bus."""
    for motor_id in motors:
        counters = bus.transport.counters[motor_id]
        assert counters.sent > 0 and counters.replied == counters.sent, (motor_id, counters)
        assert (counters.timeouts, counters.bad_frames, counters.stale_frames) == (0, 0, 0), (motor_id, counters)
    bus_counters = bus.transport.bus_counters
    assert (bus_counters.unknown_id_frames, bus_counters.bad_frames, bus_counters.dropped_bytes) == (0, 0, 0)
    assert bus_counters.skipped_requests == 0
    stats = bus.attachment.stats
    assert (stats.decode_errors, stats.unanswered, stats.corrupted, stats.undelivered) == (0, 0, 0, 0), stats


def assert_balanced(bus: Bus) -> None:
    """The transport's invariant: every request sent was either answered or timed out."""
    for motor_id, counters in bus.transport.counters.items():
        assert counters.sent == counters.replied + counters.timeouts, (motor_id, counters)


# --- 1. every command through the transport -----------------------------------------------------------------------


def test_every_command_through_the_transport(bus: Bus) -> None:
    m, model, emulator = 2, MODEL, bus.emulator
    drive = emulator.drives[m]
    can = bus.protocol is WireProtocol.CAN

    # At rest and off after power-on.
    status = bus.ask(m, Bare(Command.READ_STATUS_1))
    assert isinstance(status, Status1)
    assert status.voltage_v == model.supply_voltage_v and status.errors is ErrorFlags.NONE
    assert status.temperature_c == round(model.ambient_c)
    state = bus.ask(m, Bare(Command.READ_STATUS_2))
    assert isinstance(state, MotorState)
    assert (state.iq_a, state.speed_dps, state.encoder) == (0.0, 0, drive.encoder)
    phases = bus.ask(m, Bare(Command.READ_STATUS_3))
    assert isinstance(phases, PhaseCurrents) and (phases.ia_a, phases.ib_a, phases.ic_a) == (0.0, 0.0, 0.0)
    assert phases.temperature_c == (None if can else round(model.ambient_c))  # CAN's 0x9D carries none

    # Gains: RAM write, ROM write, read back (the power cycle at the end tells RAM from ROM).
    assert bus.ask(m, Bare(Command.READ_PID)) == dataclasses.replace(model.pid, command=Command.READ_PID)
    ram = PidGains(Command.WRITE_PID_RAM, 90, 40, 45, 35, 45, 45)
    bus.ask(m, ram)
    assert bus.ask(m, Bare(Command.READ_PID)) == dataclasses.replace(ram, command=Command.READ_PID)
    rom = PidGains(Command.WRITE_PID_ROM, 110, 60, 55, 45, 55, 55)
    bus.ask(m, rom)
    assert bus.ask(m, Bare(Command.READ_PID)) == dataclasses.replace(rom, command=Command.READ_PID)
    assert drive.pid_rom == dataclasses.replace(rom, command=Command.READ_PID)

    # Acceleration: 0x34 then 0x33 returns what was written.
    accel = bus.ask(m, Bare(Command.READ_ACCELERATION))
    assert isinstance(accel, Acceleration) and accel.acceleration_dps2 == model.acceleration_dps2
    bus.ask(m, Acceleration(Command.WRITE_ACCELERATION_RAM, 20_000))
    accel = bus.ask(m, Bare(Command.READ_ACCELERATION))
    assert isinstance(accel, Acceleration) and accel.acceleration_dps2 == 20_000
    assert drive.acceleration_dps2 == 20_000

    # A position move, then the angle and encoder readings agree with the drive where it came to rest.
    moving = bus.ask(m, MultiTurnPositionSpeed(angle_deg=45.0, max_speed_dps=360.0))
    assert isinstance(moving, MotorState) and state_of(drive) is RunState.RUNNING
    assert wait_for(lambda: abs(drive.angle_deg - 45.0) < 0.05 and abs(drive.speed_dps) < 1.0)
    angle = bus.ask(m, Bare(Command.READ_MULTI_TURN_ANGLE))
    assert isinstance(angle, MultiTurnAngle)
    assert angle.angle_deg == pytest.approx(drive.angle_deg, abs=0.1)
    assert angle.angle_deg == pytest.approx(45.0, abs=0.1)
    single = bus.ask(m, Bare(Command.READ_SINGLE_TURN_ANGLE))
    assert isinstance(single, SingleTurnAngle) and single.angle_deg == pytest.approx(45.0, abs=0.1)
    encoder = bus.ask(m, Bare(Command.READ_ENCODER))
    counts = 1 << model.encoder_bits
    assert isinstance(encoder, EncoderReading)
    assert encoder.encoder_raw == pytest.approx(drive.encoder_raw, abs=2)
    assert encoder.encoder_raw == pytest.approx(45.0 / 360.0 * counts, abs=5)
    assert encoder.encoder_offset == drive.encoder_offset == model.encoder_offset
    assert encoder.encoder == (encoder.encoder_raw - encoder.encoder_offset) % counts
    state = bus.ask(m, Bare(Command.READ_STATUS_2))
    assert isinstance(state, MotorState) and abs(state.speed_dps) <= 1
    assert state.encoder == pytest.approx(drive.encoder, abs=2)

    if can:  # 0x95 exists on CAN only: the angle is zero from now on, and the motor does not move.
        assert bus.ask(m, Bare(Command.SET_ZERO_RAM)) == Bare(Command.SET_ZERO_RAM)
        angle = bus.ask(m, Bare(Command.READ_MULTI_TURN_ANGLE))
        assert isinstance(angle, MultiTurnAngle) and angle.angle_deg == pytest.approx(0.0, abs=0.1)

    # ROM zero and offset: they take effect at the next power cycle.
    zero = bus.ask(m, Bare(Command.WRITE_ZERO_ROM))
    if can:  # CAN answers with the offset it wrote: the current raw position
        assert isinstance(zero, EncoderOffset) and zero.encoder_offset == pytest.approx(drive.encoder_raw, abs=2)
    offset = EncoderOffset(Command.WRITE_ENCODER_OFFSET, 100)
    bus.ask(m, offset)

    # The position modes: each reply is a state reply of its command, and the drive runs that command.
    for message in (
        MultiTurnPosition(angle_deg=90.0),
        SingleTurnPosition(SpinDirection.CLOCKWISE, 30.0),
        SingleTurnPositionSpeed(SpinDirection.COUNTERCLOCKWISE, 40.0, 100.0),
        IncrementalPosition(angle_deg=5.0),
        IncrementalPositionSpeed(angle_deg=-5.0, max_speed_dps=50.0),
        MultiTurnPositionSpeed(angle_deg=10.0, max_speed_dps=200.0),
    ):
        bus.ask(m, message)
        setpoint = drive.setpoint
        assert setpoint is not None and setpoint.command is command_of(message)
        assert setpoint.mode is DriveLoop.POSITION and state_of(drive) is RunState.RUNNING
        if hasattr(message, "max_speed_dps"):
            assert setpoint.max_speed_dps == message.max_speed_dps
        else:
            assert setpoint.max_speed_dps == model.max_speed_dps

    # Speed, torque and open loop: the replies report what the drive does.
    bus.ask(m, SpeedControl(speed_dps=90.0))
    assert wait_for(lambda: abs(drive.speed_dps - 90.0) < 3.0)
    state = bus.ask(m, Bare(Command.READ_STATUS_2))
    assert isinstance(state, MotorState) and state.speed_dps == pytest.approx(90.0, abs=5.0)
    bus.ask(m, TorqueControl(iq_a=0.5))
    assert wait_for(lambda: abs(drive.iq_a - 0.5) < 0.01)
    state = bus.ask(m, Bare(Command.READ_STATUS_2))
    assert isinstance(state, MotorState) and state.iq_a == pytest.approx(0.5, abs=0.03)
    open_loop = bus.ask(m, OpenLoopControl(power=100))
    assert isinstance(open_loop, OpenLoopState) and open_loop.power == 100

    # Stop keeps the command, run resumes it, off forgets it.
    bus.ask(m, Bare(Command.MOTOR_STOP))
    assert state_of(drive) is RunState.STOPPED
    bus.ask(m, Bare(Command.MOTOR_RUN))
    assert state_of(drive) is RunState.RUNNING and drive.setpoint is not None
    assert drive.setpoint.command is Command.OPEN_LOOP
    bus.ask(m, Bare(Command.MOTOR_OFF))
    assert state_of(drive) is RunState.OFF and setpoint_of(drive) is None
    cleared = bus.ask(m, Bare(Command.CLEAR_ERRORS))
    assert isinstance(cleared, Status1) and cleared.errors is ErrorFlags.NONE
    assert cleared.voltage_v == model.supply_voltage_v

    if not can:  # 0x12 exists on RS485 only
        info = bus.ask(m, Bare(Command.READ_MODEL))
        assert info == ProductInfo(model.driver_name, model.motor_name, model.hardware_version, model.firmware_version)

    # A batch: every drive in one cycle, one drive twice (same key: answered first in, first out).
    batch = [Request(i, Bare(Command.READ_STATUS_1)) for i in (*MOTORS, 1)]
    replies = bus.cycle(batch)
    assert [r.motor_id for r in replies] == [*MOTORS, 1]
    for reply in replies:
        assert isinstance(reply.message, Status1) and reply.message.voltage_v == model.supply_voltage_v
        assert reply.received_s is not None
    assert replies[0].received_s is not None and replies[-1].received_s is not None
    assert replies[0].received_s <= replies[-1].received_s

    if can:  # 0x280: one frame, four replies (motors 1..4, each like 0xA1)
        currents = (0.1, 0.2, 0.3, -0.4)
        replies = bus.cycle([Request(1, MultiMotorTorque(*currents))])
        assert [r.motor_id for r in replies] == list(MOTORS)
        for reply, iq in zip(replies, currents, strict=True):
            assert isinstance(reply.message, MotorState) and reply.message.command is Command.TORQUE
            setpoint = emulator.drives[reply.motor_id].setpoint
            assert setpoint is not None and setpoint.mode is DriveLoop.TORQUE
            assert setpoint.value == pytest.approx(iq, abs=0.016)  # the wire carries 32/2000 A steps
        replies = bus.cycle([Request(i, Bare(Command.MOTOR_OFF)) for i in MOTORS])
        assert all(r.message == Bare(Command.MOTOR_OFF) for r in replies)

    # Power cycle: RAM gains and acceleration are lost, ROM gains and the written offset take effect.
    emulator.power_cycle(m)
    assert bus.ask(m, Bare(Command.READ_PID)) == dataclasses.replace(rom, command=Command.READ_PID)
    accel = bus.ask(m, Bare(Command.READ_ACCELERATION))
    assert isinstance(accel, Acceleration) and accel.acceleration_dps2 == model.acceleration_dps2
    encoder = bus.ask(m, Bare(Command.READ_ENCODER))
    assert isinstance(encoder, EncoderReading) and encoder.encoder_offset == 100

    # Commands the protocol lacks are refused before anything of the cycle is sent.
    lacking: list[Message] = [
        Bare(code) for code, spec in COMMANDS.items() if spec.layout(bus.protocol, Direction.REQUEST) is None
    ]
    if not can:
        lacking.append(MultiMotorTorque(0.0, 0.0, 0.0, 0.0))  # RS485 has no broadcast
    assert lacking
    sent, cycles = bus.transport.counters[m].sent, bus.transport.bus_counters.cycles
    requests_seen = bus.attachment.stats.requests
    for refused in lacking:
        with pytest.raises(EncodeError):
            bus.cycle([Request(m, Bare(Command.READ_STATUS_1)), Request(m, refused)])
    time.sleep(QUIET_S)
    assert bus.attachment.stats.requests == requests_seen
    assert (bus.transport.counters[m].sent, bus.transport.bus_counters.cycles) == (sent, cycles)

    # Every request command of the protocol went through the transport, and every reply was matched.
    expected = {code for code, spec in COMMANDS.items() if spec.layout(bus.protocol, Direction.REQUEST) is not None}
    assert bus.exercised == expected
    assert_clean(bus)


# --- 2. fault kinds through the transport -------------------------------------------------------------------------


def test_silent_drive_times_out_by_the_deadline_and_recovers(bus: Bus) -> None:
    drive = bus.emulator.drives[3]
    bus.ask(3, SpeedControl(speed_dps=60.0))  # running before it falls silent
    fault = bus.fault(InjectedFault.SILENT, 3, lasting_s=0.5)
    deadline = bus.transport.clock() + 2 * DEADLINE_S
    replies = bus.transport.transact([Request(1, Bare(Command.READ_STATUS_1)), Request(3, SpeedControl(-60.0))],
                                     deadline)  # fmt: skip
    # The transport waited for the silent drive until the deadline, and not much longer (a loose bound).
    assert deadline <= bus.transport.clock() < deadline + 1.0
    assert [r.motor_id for r in replies] == [1, 3]
    assert isinstance(replies[0].message, Status1)
    assert replies[1].message is None and replies[1].received_s is None and not replies[1].ok
    counters = bus.transport.counters[3]
    assert (counters.sent, counters.replied, counters.timeouts, counters.stale_frames) == (2, 1, 1, 0)
    # Not heard: the drive keeps running its last command.
    assert drive.setpoint is not None and drive.setpoint.value == 60.0
    assert wait_for(lambda: bus.attachment.stats.unanswered == 1)

    assert fault.end_s is not None
    bus.wait_sim(fault.end_s)
    # The one-reply ambiguity (motion.transport.base): the first reply with the expired request's key is presumed
    # the late answer, counted stale, never matched; the drive did execute the request.
    (reply,) = bus.cycle([Request(3, SpeedControl(-60.0))])
    assert reply.message is None
    assert (counters.stale_frames, counters.timeouts) == (1, 2)
    assert drive.setpoint is not None and drive.setpoint.value == -60.0
    # That costs one cycle, not more.
    (reply,) = bus.cycle([Request(3, SpeedControl(-60.0))])
    assert isinstance(reply.message, MotorState) and reply.message.command is Command.SPEED
    state = bus.ask(3, Bare(Command.READ_STATUS_2))
    assert isinstance(state, MotorState)
    assert (counters.sent, counters.replied, counters.timeouts, counters.stale_frames) == (5, 3, 2, 1)
    assert_balanced(bus)
    assert bus.transport.counters[1].replied == bus.transport.counters[1].sent


def test_dropped_requests_get_no_reply_and_are_not_executed(bus: Bus) -> None:
    drive = bus.emulator.drives[4]
    fault = bus.fault(InjectedFault.DROP, 4, lasting_s=0.5)  # probability 1
    replies = bus.cycle([Request(1, Bare(Command.READ_STATUS_2)), Request(4, MultiTurnPosition(angle_deg=30.0))])
    assert isinstance(replies[0].message, MotorState) and replies[1].message is None
    assert drive.setpoint is None and state_of(drive) is RunState.OFF
    if bus.protocol is WireProtocol.CAN:  # one 0x280 frame: motors 1..3 answer, the dropped one does not
        replies = bus.cycle([Request(1, MultiMotorTorque(0.1, 0.1, 0.1, 0.1))])
        assert [r.motor_id for r in replies] == list(MOTORS)
        assert [r.ok for r in replies] == [True, True, True, False]
        assert drive.setpoint is None
        bus.cycle([Request(i, Bare(Command.MOTOR_OFF)) for i in (1, 2, 3)])
    counters = bus.transport.counters[4]
    dropped = counters.sent
    assert counters.timeouts == dropped and counters.replied == counters.stale_frames == 0
    # The attachment counts the request that nobody answered (0x280 was answered by the others), and notes each
    # dropped request in the frame log.
    assert wait_for(lambda: bus.attachment.stats.unanswered == 1 and len(bus.log("NOTE")) == dropped)

    assert fault.end_s is not None
    bus.wait_sim(fault.end_s)
    # After the fault the drive answers again (another key than the expired ones, so no presumed-late discard).
    status = bus.ask(4, Bare(Command.READ_STATUS_1))
    assert isinstance(status, Status1)
    assert counters.replied == 1 and counters.stale_frames == 0
    assert_balanced(bus)


def test_late_reply_is_stale_in_the_next_cycle_and_never_matched(bus: Bus) -> None:
    drive = bus.emulator.drives[2]
    delay_s = 0.4
    bus.fault(InjectedFault.DELAY, 2, value=delay_s * 1000.0)  # longer than the first cycle's deadline
    first = PidGains(Command.WRITE_PID_RAM, 91, 41, 46, 36, 46, 46)
    second = PidGains(Command.WRITE_PID_RAM, 92, 42, 47, 37, 47, 47)
    replies = bus.cycle([Request(1, Bare(Command.READ_STATUS_1)), Request(2, first)])
    assert isinstance(replies[0].message, Status1)
    assert replies[1].message is None  # late: no reply this cycle
    assert drive.pid == dataclasses.replace(first, command=Command.READ_PID)  # executed; only the reply is late
    counters = bus.transport.counters[2]
    assert (counters.timeouts, counters.stale_frames) == (1, 0)

    # Next cycle, same key: the late echo of `first` arrives (before or during this cycle) and is counted stale;
    # this cycle's own reply, delayed too, is the one matched.
    (reply,) = bus.cycle([Request(2, second)], budget_s=delay_s + 1.0)
    assert reply.message == second, "the late reply of the previous cycle was matched to this request"
    assert (counters.sent, counters.replied, counters.timeouts, counters.stale_frames) == (2, 1, 1, 1)
    # Status 1 and both echoes: every reply sent was taken in. (The attachment counts a reply after writing it.)
    assert wait_for(lambda: bus.attachment.stats.replies == 3)
    assert_balanced(bus)


@pytest.mark.parametrize("corruption", list(Corruption), ids=[c.value for c in Corruption])
def test_corrupt_replies_are_counted_and_never_matched(bus: Bus, corruption: Corruption) -> None:
    bus.fault(InjectedFault.CORRUPT, 3, corruption=corruption)
    pair = [Request(1, Bare(Command.READ_STATUS_1)), Request(3, Bare(Command.READ_STATUS_1))]
    replies = bus.cycle(pair, budget_s=DEADLINE_S)
    assert isinstance(replies[0].message, Status1) and replies[0].motor_id == 1
    assert replies[1].message is None
    assert wait_for(lambda: bus.attachment.stats.corrupted == 1)  # the drive did answer, damaged
    counters, bus_counters = bus.transport.counters[3], bus.transport.bus_counters
    assert (counters.sent, counters.replied, counters.timeouts, counters.stale_frames) == (1, 0, 1, 0)
    if bus.protocol is WireProtocol.CAN and corruption is Corruption.ID:
        # 0x100 + id is no drive's reply id: counted on the bus, not attributable to a motor.
        assert bus_counters.unknown_id_frames == 1 and counters.bad_frames == 0
    else:
        # CAN: command byte 0x00 or a 7-byte payload; RS485: data checksum, motor id 0, truncated frame.
        assert counters.bad_frames == 1 and bus_counters.unknown_id_frames == 0
    if bus.protocol is WireProtocol.RS485:
        assert bus_counters.dropped_bytes > 0
    for motor_id in (1, 2, 4):
        assert motor_id not in bus.transport.counters or bus.transport.counters[motor_id].bad_frames == 0
    assert bus.transport.counters[1].stale_frames == 0
    assert_balanced(bus)


@pytest.mark.parametrize(
    ("kind", "flag"),
    [
        (InjectedFault.OVER_TEMPERATURE, ErrorFlags.OVER_TEMPERATURE),
        (InjectedFault.UNDER_VOLTAGE, ErrorFlags.LOW_VOLTAGE),
    ],
    ids=["over_temperature", "under_voltage"],
)
def test_protection_flag_latches_while_the_cause_persists(bus: Bus, kind: InjectedFault, flag: ErrorFlags) -> None:
    m, model = 1, MODEL
    drive = bus.emulator.drives[m]
    status = bus.ask(m, Bare(Command.READ_STATUS_1))
    assert isinstance(status, Status1) and status.errors is ErrorFlags.NONE
    fault = bus.fault(kind, m, lasting_s=0.4, after_s=0.05)

    status = bus.ask(m, Bare(Command.READ_STATUS_1))
    assert isinstance(status, Status1) and status.errors & flag
    if kind is InjectedFault.OVER_TEMPERATURE:
        assert status.temperature_c > model.over_temperature_c
    else:
        assert status.voltage_v < model.low_voltage_v
    # While the flag is set the power stage stays off: control commands are answered but not run.
    bus.ask(m, SpeedControl(speed_dps=100.0))
    assert state_of(drive) is RunState.OFF
    cleared = bus.ask(m, Bare(Command.CLEAR_ERRORS))
    assert isinstance(cleared, Status1) and cleared.errors & flag  # the cause persists: not cleared

    assert fault.end_s is not None
    bus.wait_sim(fault.end_s)
    if kind is InjectedFault.OVER_TEMPERATURE:
        assert wait_for(lambda: drive.temperature_c <= model.over_temperature_c)  # cools after the fault
    status = bus.ask(m, Bare(Command.READ_STATUS_1))
    assert isinstance(status, Status1) and status.errors & flag  # latched until 0x9B
    assert status.temperature_c <= model.over_temperature_c and status.voltage_v == model.supply_voltage_v
    cleared = bus.ask(m, Bare(Command.CLEAR_ERRORS))
    assert isinstance(cleared, Status1) and cleared.errors is ErrorFlags.NONE
    status = bus.ask(m, Bare(Command.READ_STATUS_1))
    assert isinstance(status, Status1) and status.errors is ErrorFlags.NONE
    bus.ask(m, SpeedControl(speed_dps=100.0))
    assert state_of(drive) is RunState.RUNNING
    bus.ask(m, Bare(Command.MOTOR_OFF))
    assert_clean(bus, (m,))


# --- 3. protocol-breaking requests to the emulator ----------------------------------------------------------------

BROKEN_CAN = [
    CanFrame(0x142, bytes(8)),  # command 0x00
    CanFrame(0x142, bytes.fromhex("9a 00 00 00 00 00 00")),  # 7-byte payload
    CanFrame(0x142, bytes.fromhex("12 00 00 00 00 00 00 00")),  # 0x12 exists on RS485 only
    CanFrame(0x142, bytes.fromhex("9a 00 00 00 00 00 00 01")),  # reserved byte set
    CanFrame(0x280, bytes.fromhex("ff 7f 00 00 00 00 00 00")),  # 0x280 current above the +-32 A range
]
_STATUS_1_OF_2 = rs485_frame.encode_request(Bare(Command.READ_STATUS_1), 2)
#: RS485 input that breaks the protocol, and whether it is a checksum-valid frame (counted exactly once).
BROKEN_RS485 = [
    (bytes.fromhex("01 02 03 04 05 06"), False),  # line noise, no frame head
    (_STATUS_1_OF_2[:4] + bytes([_STATUS_1_OF_2[4] ^ 0x55]), False),  # header checksum
    (Rs485Frame(0x00, 2, b"").to_bytes(), True),  # no such command
    (Rs485Frame(0x95, 2, b"").to_bytes(), True),  # 0x95 exists on CAN only
    (Rs485Frame(0x9A, 2, b"\x00").to_bytes(), True),  # 0x9A carries no data
]


def _send_broken_can(bus: Bus) -> list[str]:
    path = bus.attachment.path
    kwargs: dict[str, Any] = {"bitrate": 1_000_000, "sleep_after_open": 0} if bus.kind == "slcan" else {}
    with CanEndpoint(bus.kind, path, **kwargs) as host:
        for n, frame in enumerate(BROKEN_CAN, start=1):
            host.send(frame)
            assert wait_for(decode_errors_reach(bus, n))
            assert host.recv(QUIET_S) is None, f"broken frame {frame} was answered"
    return [f"{frame.arbitration_id:03X}: {frame.data.hex(' ')}" for frame in BROKEN_CAN]


def _send_broken_rs485(bus: Bus) -> list[str]:
    with serial.Serial(bus.attachment.path, 115_200, timeout=QUIET_S) as port:
        for raw, framed in BROKEN_RS485:
            before = bus.attachment.stats.decode_errors
            port.write(raw)
            assert wait_for(decode_errors_reach(bus, before + 1))
            assert port.read(64) == b"", f"broken input {raw.hex(' ')} was answered"
            if framed:  # a checksum-valid frame is one protocol error, whatever the pty's pace
                assert bus.attachment.stats.decode_errors == before + 1
    return [raw.hex(" ") for raw, framed in BROKEN_RS485 if framed]


def test_protocol_breaking_requests_are_counted_logged_and_not_answered(bus: Bus) -> None:
    bus.ask(2, Bare(Command.READ_STATUS_1))
    stats = bus.attachment.stats
    assert wait_for(lambda: stats.replies == 1)  # counted after it was written, maybe after the host read it
    # The host port is free for a raw sender (RS485 locks it; a CAN host would see the raw frames as traffic).
    bus.transport.close()
    wires = _send_broken_rs485(bus) if bus.kind == "rs485" else _send_broken_can(bus)
    assert stats.replies == 1 and stats.unanswered == 0
    assert stats.decode_errors >= len(BROKEN_CAN if bus.protocol is WireProtocol.CAN else BROKEN_RS485)
    bad = bus.log("BAD")
    assert len(bad) == stats.decode_errors
    if bus.protocol is WireProtocol.CAN:
        assert bad == wires
    else:
        assert set(wires) <= set(bad)
    assert bus.emulator.drives[2].state is RunState.OFF  # nothing was executed

    # The line still works, and nothing answers a broken request late.
    bus.open_transport()
    time.sleep(QUIET_S)
    status = bus.ask(2, Bare(Command.READ_STATUS_1))
    assert isinstance(status, Status1)
    counters = bus.transport.counters[2]
    assert (counters.sent, counters.replied, counters.stale_frames, counters.bad_frames) == (1, 1, 0, 0)
    assert bus.transport.bus_counters.unknown_id_frames == 0
    errors = stats.decode_errors
    assert wait_for(lambda: stats.replies == 2)
    time.sleep(QUIET_S)
    assert (stats.replies, stats.decode_errors) == (2, errors)
