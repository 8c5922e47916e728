"""An arm on several buses (issue 35): one trajectory over both, each cycle's batches on the buses at the same time,
and one safety domain (a fault on either bus halts every axis on both in its detection cycle)."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import shutil
import signal
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from motion.api import Arm
from motion.cli.moves import _jog_verdict
from motion.compose import axis_specs
from motion.config import ArmConfig, ControlMode
from motion.control.ratecheck import RateError
from motion.emulator import Emulator, VirtualCanAttachment
from motion.emulator.faults import Fault, InjectedFault
from motion.emulator.simulated import SimulatedBus, Simulation
from motion.errors import MotionFault, TransportError
from motion.keep import TURNS_SCHEMA, TURNS_VERSION, load_turn_records, turns_store
from motion.protocol import Bare, Command, MotorState, MultiMotorTorque, Status1
from motion.protocol.table import ADDRESS_STRIDE, ProtocolFamily
from motion.safety import ArmState
from motion.telemetry import load_log
from motion.transport import CanTransport, Request
from motion.transport.buses import WORKER_GRACE_S, Buses
from tests.motion_rig import (
    Rig,
    arm_config,
    commanded_positions,
    emulated_arm,
    logged_requests,
    received,
    skip_if_rate_refused,
)
from tests.test_cli import cli, host_stall_misses

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"
#: As tests/test_cli.py's moving tests: half the rate check's highest rate, and none below 50 Hz.
RATE_SHARE, MIN_RATE_HZ = 0.5, 50.0
BIMANUAL = arm_config("bimanual.yaml")
#: Both arms move: each its own way (different distances on each joint, so that Ruckig's synchronisation matters).
TARGETS = np.array([30.0, -25.0, 40.0, 20.0, -15.0, 10.0, -35.0, 20.0, -30.0, -10.0, 25.0, -20.0])


def _addresses() -> list[int]:
    return [j.address for j in BIMANUAL.joints]


def test_both_arms_move_together_and_every_joint_arrives_within_one_cycle_of_the_others(tmp_path: Path) -> None:
    with emulated_arm(BIMANUAL, "sim", tmp_path, supervised=True) as rig:
        supervisor = rig.supervisor
        assert supervisor is not None
        references: list[np.ndarray] = []
        rig.controller.cycle_hooks.append(lambda c, _start, _replies: references.append(c.reference.position.copy()))
        supervisor.move_to(TARGETS, 1.0)
        assert supervisor.wait(20.0)
        # one trajectory over both buses: every joint's reference reaches its target in the same cycle (within one)
        reference = np.array(references)
        arrived = [int(np.argmax(np.abs(reference[:, i] - TARGETS[i]) < 1e-9)) for i in range(len(TARGETS))]
        assert all(np.abs(reference[a:, i] - TARGETS[i]).max() < 1e-9 for i, a in enumerate(arrived))
        assert max(arrived) - min(arrived) <= 1, arrived
        assert min(arrived) > 100  # (a real move: well over 100 cycles at 250 Hz)
        # and the drives followed: every joint within the goal tolerance when the move returned
        tolerance = BIMANUAL.control.goal_tolerance_deg
        np.testing.assert_allclose(rig.controller.snapshot.position_deg, TARGETS, atol=tolerance)
        # the set-points each drive received on its bus (both buses' 0xA4 streams, joint angles on the cycle grid)
        commanded = commanded_positions(rig)
        np.testing.assert_allclose(commanded[-1], TARGETS, atol=2e-3)  # (the 0xA4 field's 0.01 motor deg)
    assert set(received(rig, Command.MULTI_TURN_POSITION_SPEED)) == set(_addresses())


def test_each_cycle_carries_both_buses_batches_at_the_same_time(tmp_path: Path) -> None:
    # simulated wire time: the last 0xA4 of a cycle reaches its drive at the same instant on both buses (each bus
    # carries six frames), not one bus's time later
    with emulated_arm(BIMANUAL, "sim", tmp_path, supervised=True) as rig:
        assert rig.supervisor is not None
        rig.supervisor.move_to(TARGETS, 1.0)
        rig.sleep(0.3)
    last = {key: max(times) for key, times in setpoint_arrivals(rig).items()}
    cycles = sorted({cycle for cycle, _ in last})
    assert len(cycles) > 50
    skew = [abs(last[(c, 1)] - last[(c, 0)]) for c in cycles if (c, 0) in last and (c, 1) in last]
    assert max(skew) < 20e-6, max(skew)  # (one 0xA4 frame takes about 130 us at 1 Mbit/s)


def setpoint_arrivals(rig: Rig) -> dict[tuple[int, int], list[float]]:
    """(cycle, bus) -> when each 0xA4 of that cycle reached its drive on that bus (the n-th 0xA4 a drive received
    is the n-th cycle's)."""
    arrivals: dict[tuple[int, int], list[float]] = {}
    counts: dict[int, int] = {}
    for t, address, message in logged_requests(rig):
        if address is None or getattr(message, "command", None) != Command.MULTI_TURN_POSITION_SPEED:
            continue
        counts[address] = counts.get(address, 0) + 1
        arrivals.setdefault((counts[address], address // ADDRESS_STRIDE), []).append(t)
    return arrivals


def _halted_everywhere_in_the_detection_cycle(rig: Rig) -> None:
    supervisor = rig.supervisor
    assert supervisor is not None and supervisor.halts
    halt, period = supervisor.halts[0], rig.controller.period_s
    assert halt.halt_sent_s - halt.detected_s < period
    rig.sleep(period)  # (an RS485 line's last frames of that cycle may still be on the simulated wire)
    stops = received(rig, Command.MOTOR_STOP)
    for joint in rig.config.joints:
        first = min(stops.get(joint.address, [np.inf]))
        assert halt.detected_s <= first < halt.detected_s + period, (joint.name, first - halt.detected_s)


@pytest.mark.parametrize(
    ("kind", "address", "value", "expected"),
    [
        (InjectedFault.OVER_TEMPERATURE, 103, 90.0, "drive_over_temperature"),  # right elbow's drive flag
        (InjectedFault.SILENT, 105, None, "no_reply"),  # right wrist_pitch's drive falls silent
        (InjectedFault.OVER_TEMPERATURE, 2, 90.0, "drive_over_temperature"),  # the left bus's shoulder
    ],
)
def test_a_fault_on_one_bus_halts_every_axis_on_both_in_its_detection_cycle(
    tmp_path: Path, kind: InjectedFault, address: int, value: float | None, expected: str
) -> None:
    # our own temperature limit above the drive's protection (80 degC): the 0x9A flag is what trips
    joints = tuple(dataclasses.replace(j, temperature_limit_c=100.0) for j in BIMANUAL.joints)
    fault_halts_every_axis(dataclasses.replace(BIMANUAL, joints=joints), tmp_path, kind, address, value, expected)


def fault_halts_every_axis(
    config: ArmConfig,
    tmp_path: Path,
    kind: InjectedFault,
    address: int,
    value: float | None,
    expected: str,
    *,
    after_s: float = 0.4,
    family: tuple[ProtocolFamily, ...] | None = None,
) -> None:
    """Inject ``kind`` on drive ``address`` ``after_s`` into a move of every joint (in simulated time; ``family``:
    each bus's drives' generation): the fault is ``expected``, named on its joint, and every axis on every bus
    received its halt in the detection cycle."""
    with emulated_arm(config, "sim", tmp_path, supervised=True, family=family) as rig:
        supervisor = rig.supervisor
        assert supervisor is not None
        supervisor.move_to(TARGETS, 0.5)
        rig.sleep(after_s)
        now = rig.emulator.time_s
        end_s = None if kind is InjectedFault.POWER_CYCLE else now + 60.0  # (a power cycle is one instant)
        rig.emulator.add_fault(Fault(kind, address, start_s=now, end_s=end_s, value=value))
        with pytest.raises(MotionFault) as info:
            supervisor.wait(10.0)
        assert info.value.kind == expected
        assert info.value.joint == next(j.name for j in config.joints if j.address == address)
        _halted_everywhere_in_the_detection_cycle(rig)
        assert supervisor.state in (ArmState.HALTING, ArmState.HALTED)


def _realtime(config: ArmConfig) -> ArmConfig:
    """``config`` as the real-time rigs run it: at 50 Hz, with a quarter of a second for a reply (a busy host keeps an
    in-process emulator waiting; silence itself is asserted in simulated time above)."""
    safety = dataclasses.replace(config.safety, reply_timeout_ms=250.0)
    return dataclasses.replace(config, control=dataclasses.replace(config.control, rate_hz=50.0), safety=safety)


def test_a_bus_lost_in_real_time_halts_the_other_buses_drives_in_its_detection_cycle(tmp_path: Path) -> None:
    # the right bus's adapter goes (its pty closes under the host): the left bus's six drives get their 0x81 in the
    # cycle that found the port gone; they are then halted as usual (acknowledged: HALTED, and the session's end halts
    # them again), while the right bus's drives, unreachable, read as silent drives whose halt is owed
    with emulated_arm(_realtime(BIMANUAL), "slcan", tmp_path, supervised=True) as rig:
        supervisor = rig.supervisor
        assert supervisor is not None
        supervisor.move_to(TARGETS, 0.5)
        rig.sleep(0.4)
        assert supervisor.state is ArmState.MOVING
        rig.attachments[1].close()
        with pytest.raises(MotionFault) as info:
            supervisor.wait(5.0)
        assert info.value.kind == "transport" and "bus right:" in str(info.value) and "port is gone" in str(info.value)
        rig.sleep(0.6)  # (the halt's retry window: 0x81 to every drive not known to be halted)
        assert supervisor.machine.state is ArmState.HALTED
        assert supervisor.unacknowledged == {j.address for j in BIMANUAL.joints_on(1)}
        assert not rig.controller.bus.closed  # (the left bus is still reachable)
        halt = supervisor.halts[0]
        stops = received(rig, Command.MOTOR_STOP)
        for joint in BIMANUAL.joints_on(0):
            first = min(stops.get(joint.address, [np.inf]))
            assert halt.detected_s <= first < halt.detected_s + rig.controller.period_s, joint.name
        assert not any(a >= ADDRESS_STRIDE for a in stops)  # (nothing reaches the lost bus)
    closing = received(rig, Command.MOTOR_STOP)
    assert all(len(closing[j.address]) > len(stops[j.address]) for j in BIMANUAL.joints_on(0))  # halted at close too


def test_the_cli_moves_both_arms_in_real_time_against_the_emulator_on_two_slcan_ptys(tmp_path: Path) -> None:
    # `rmd-motion emulate --config bimanual.yaml --slcan-link left=... --slcan-link right=...`, then `move` of all
    # twelve joints with `--channel BUS=...` per bus: every joint at its target when the move returns
    links = {name: tmp_path / f"slcan-{name}" for name in ("left", "right")}
    command = [sys.executable, "-m", "motion.cli", "emulate", "--config", str(CONFIGS / "bimanual.yaml")]
    for name, link in links.items():
        command += ["--slcan-link", f"{name}={link}"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert process.stdout is not None
        started = [process.stdout.readline() for _ in range(3)]
        assert started[0].startswith(f"slcan: {links['left']}") and "(bus left)" in started[0], started
        assert f"{links['right']}" in started[1] and "(bus right)" in started[1], started
        assert "on bus left" in started[2] and "on bus right" in started[2], started
        bus = ["--interface", "slcan", *(a for n, p in links.items() for a in ("--channel", f"{n}={p}"))]
        checked = cli("check", "--config", CONFIGS / "bimanual.yaml", *bus, "--json")
        assert checked.returncode in {0, 2}, checked.stderr
        data = json.loads(checked.stdout)
        highest = float(data["modes"]["position"]["highest_rate_hz"]) * RATE_SHARE
        if highest < MIN_RATE_HZ:
            pytest.skip(f"this host holds no rate the moving tests run bimanual.yaml at (rate check: {highest:g} Hz)")
        config = _copy_at(tmp_path, min(round(highest), 250))
        targets = [f"{j.name}={t:g}" for j, t in zip(BIMANUAL.joints, TARGETS, strict=True)]
        trace = tmp_path / "move.log"
        moved = cli("move", "--config", config, *bus, "--speed-scale", "0.5", *targets, "--json", "--trace", trace)
        skip_if_rate_refused(moved)
        assert moved.returncode == 0, moved.stderr
        assert json.loads(moved.stdout)["arrival"]["arrived"]
        # the trace: the frames of both buses (each bus's worker thread), each on its bus, both sent and taken in
        traced = {tuple(line.split()[1::2]) for line in trace.read_text().splitlines()}
        assert {(b, d) for b in ("left", "right") for d in "TR"} <= traced
        status = cli("status", "--config", config, *bus, "--json")
        assert status.returncode == 0, status.stderr
        joints = json.loads(status.stdout)["joints"]
        assert [(j["name"], j["bus"], j["motor_id"]) for j in joints] == [
            (j.name, j.bus, j.motor_id) for j in BIMANUAL.joints
        ]
        tolerance = BIMANUAL.control.goal_tolerance_deg
        np.testing.assert_allclose([j["position_deg"] for j in joints], TARGETS, atol=tolerance + 0.01)
    finally:
        process.send_signal(signal.SIGTERM)
        process.communicate(timeout=10)


def _copy_at(tmp_path: Path, rate_hz: float) -> Path:
    """bimanual.yaml (and its URDF) in ``tmp_path`` at ``rate_hz``, with a quarter of a second for a reply and its
    cycles of missed replies (a busy host; silence is asserted in simulated time above)."""
    shutil.copy(CONFIGS / "bimanual.urdf", tmp_path / "bimanual.urdf")
    text = (CONFIGS / "bimanual.yaml").read_text()
    text = text.replace("rate_hz: 250", f"rate_hz: {rate_hz:g}").replace("reply_timeout_ms: 5", "reply_timeout_ms: 250")
    misses = f"max_missed_replies: {host_stall_misses(rate_hz)}"
    text = text.replace("max_missed_replies: 2", misses)
    assert f"rate_hz: {rate_hz:g}" in text and "reply_timeout_ms: 250" in text and misses in text
    path = tmp_path / "bimanual.yaml"
    path.write_text(text)
    return path


def test_torque_mode_sends_one_0x280_frame_per_bus_for_its_motors_1_to_4(tmp_path: Path) -> None:
    config = arm_config("bimanual.yaml", mode=ControlMode.TORQUE, rate_hz=250)
    with emulated_arm(config, "sim", tmp_path, supervised=True) as rig:
        assert rig.supervisor is not None
        rig.supervisor.move_to(TARGETS * 0.2, 1.0)
        assert rig.supervisor.wait(20.0)
    frames: dict[str, int] = {}
    torque: set[int] = set()
    for line in rig.frame_log.read_text().splitlines():
        fields = line.split(maxsplit=3)
        if len(fields) == 4 and fields[1] == "IN" and fields[3].startswith("280:"):
            frames[fields[2]] = frames.get(fields[2], 0) + 1
    for _, address, message in logged_requests(rig):
        if address is not None and getattr(message, "command", None) == Command.TORQUE:
            torque.add(address)
    assert len(frames) == 2 and min(frames.values()) > 100, frames  # both buses, every cycle
    assert torque == {5, 6, 105, 106}  # each bus's motors beyond 4 by 0xA1


def test_the_command_line_refuses_overrides_that_do_not_name_each_bus(tmp_path: Path) -> None:
    config = CONFIGS / "bimanual.yaml"
    plain = cli("status", "--config", config, "--interface", "slcan", "--channel", "/dev/ttyACM0")
    assert plain.returncode == 2 and "has several buses (left, right): give --channel BUS=VALUE" in plain.stderr
    twice = cli("status", "--config", config, "--channel", "left=/a", "--channel", "left=/b")
    assert twice.returncode == 2 and "--channel is given twice for bus left" in twice.stderr
    port = cli("status", "--config", config, "--port", "left=/dev/ttyUSB0")
    assert port.returncode == 2 and "bus left is a can bus; its overrides are --interface and --channel" in port.stderr
    mixed = cli("status", "--config", config, "--interface", "slcan", "--interface", "left=socketcan")
    assert mixed.returncode == 2 and "--interface: give BUS=VALUE for every bus it overrides, or one" in mixed.stderr
    one = cli("status", "--config", CONFIGS / "arm2.yaml", "--channel", "/a", "--channel", "/b")
    assert one.returncode == 2 and "--channel is given 2 times: the arm has one bus" in one.stderr


@pytest.mark.parametrize(
    ("links", "message"),
    [
        (["left={0}/l"], "no link for bus(es) right"),
        (["left={0}/l", "{0}/r"], "the arm is on several buses: give BUS=PATH"),
        (["left={0}/l", "middle={0}/m"], "no bus 'middle'; the buses are left, right"),
        (["left={0}/l", "left={0}/m"], "bus left has a link already"),
    ],
)
def test_emulate_takes_one_link_per_bus(tmp_path: Path, links: list[str], message: str) -> None:
    args = [a for link in links for a in ("--slcan-link", link.format(tmp_path))]
    result = cli("emulate", "--config", CONFIGS / "bimanual.yaml", *args)
    assert result.returncode == 2 and message in result.stderr, result.stderr
    rs485 = cli("emulate", "--config", CONFIGS / "bimanual.yaml", "--rs485-link", f"left={tmp_path}/l")
    assert rs485.returncode == 2 and "bus left is a can bus" in rs485.stderr, rs485.stderr


def test_a_recording_of_both_arms_names_each_joints_bus(tmp_path: Path) -> None:
    recording, trace = tmp_path / "run.mcap", tmp_path / "run.log"
    moved = cli(
        "move", "--config", CONFIGS / "bimanual.yaml", "--emulate", "--log", recording, "--trace", trace,
        "right_base_yaw=10",
    )  # fmt: skip
    assert moved.returncode == 0, moved.stderr
    # the trace: each frame on its bus's interface (named as the bus), both buses' 0xA4 to their motor 1
    lines = [line.split() for line in trace.read_text().splitlines()]
    assert {fields[1] for fields in lines} == {"left", "right"}
    sent = {(fields[1], fields[2][:6]) for fields in lines if fields[3] == "T"}
    assert {("left", "141#A4"), ("right", "141#A4")} <= sent
    # the recording's frames name their bus the same way
    with AnyReader([recording]) as reader:
        connections = [c for c in reader.connections if c.topic == "/bus/frames"]
        frames: list[Any] = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections)]
    assert len(frames) == len(lines) and {f.bus for f in frames} == {"left", "right"}
    in_recording = sum(f.bus == "right" and f.arbitration_id == 0x141 and not f.received for f in frames)
    in_trace = sum(fields[1] == "right" and fields[2].startswith("141#") and fields[3] == "T" for fields in lines)
    assert in_recording == in_trace > 0
    log = load_log(recording)
    assert [b["name"] for b in log.meta["buses"]] == ["left", "right"]
    assert [(j["name"], j["bus"], j["motor_id"]) for j in log.meta["joints"]] == [
        (j.name, j.bus, j.motor_id) for j in BIMANUAL.joints
    ]
    assert log.meta["channel"] == "left=can0, right=can1"
    final = log.columns["q_deg"][-1]
    assert abs(final[6] - 10.0) < BIMANUAL.control.goal_tolerance_deg + 0.01  # right_base_yaw, the 7th joint


def test_jog_of_a_joint_on_the_second_bus_names_its_drive_there() -> None:
    # the jog verdict compares the drives that turned (by address) with the joint's: motor 2 of the right bus is not
    # motor 2 of the left one
    specs = {s.motor_id: s for s in axis_specs(BIMANUAL)}
    joint = BIMANUAL.joints[7]  # right_shoulder_pitch
    verdict = _jog_verdict(joint, 36.0, [(specs[102], 35.8)], 1.0)
    assert "right_shoulder_pitch (motor 2 on bus right) turned +35.8 motor deg, as commanded" in verdict
    other = _jog_verdict(joint, 36.0, [(specs[2], 35.8)], 1.0)
    assert "turned: motor 2 on bus left (left_shoulder_pitch) +35.8 motor deg" in other


def test_the_rate_check_measures_each_bus_and_names_the_one_that_limits() -> None:
    with Arm.from_config(CONFIGS / "bimanual.yaml", emulate=True) as arm:
        check = arm.rate_check
    assert check is not None and [name for name, _ in check.by_bus_p99_s] == ["left", "right"]
    assert all(0.0 < t <= check.round_trip_p99_s for _, t in check.by_bus_p99_s)
    assert "by bus (p99, at the same time): left" in check.summary() and "limits" in check.summary()


@pytest.mark.parametrize("parallel", [True, False], ids=["parallel", "sequential"])
def test_the_buses_transport_merges_replies_in_request_order_by_address(parallel: bool) -> None:
    # two virtual CAN buses of one emulator (lines 0 and 1); a batch that mixes them, with a 0x280 frame on the second
    emulator = Emulator([1, 2, 3, 4, 101, 102, 103, 104])
    channels = [uuid.uuid4().hex, uuid.uuid4().hex]
    with contextlib.ExitStack() as stack:
        for line, channel in enumerate(channels):
            stack.enter_context(VirtualCanAttachment(emulator, channel, line=line))
        transports = [CanTransport("virtual", c, None) for c in channels]
        buses = stack.enter_context(Buses(transports, ["left", "right"], parallel=parallel))
        requests = [
            Request(102, Bare(Command.READ_STATUS_2)),
            Request(1, Bare(Command.READ_STATUS_1)),
            Request(101, MultiMotorTorque(0.0, 0.0, 0.0, 0.0)),
            Request(2, Bare(Command.READ_STATUS_2)),
        ]
        replies = buses.transact(requests, buses.clock() + 0.5)
        assert [(r.motor_id, r.ok) for r in replies] == [
            (102, True), (1, True), (101, True), (102, True), (103, True), (104, True), (2, True)
        ]  # fmt: skip
        assert isinstance(replies[1].message, Status1) and isinstance(replies[2].message, MotorState)
        assert buses.counters[103].replied == 1 and buses.motor_counters(103) is buses.buses[1].counters[3]
        assert set(buses.bus_times_s() or {}) == {"left", "right"}
        assert buses.describe().startswith("left: can virtual:") and ", right: can virtual:" in buses.describe()
        with pytest.raises(TransportError, match="no bus 2"):
            buses.transact([Request(201, Bare(Command.READ_STATUS_1))], buses.clock() + 0.1)


class _Stalling(CanTransport):
    """A backend whose exchange blocks (a write that never returns, a wedged driver) until released."""

    release = threading.Event()

    def _exchange(self, deadline_s: float) -> None:
        self.release.wait(5.0)
        super()._exchange(deadline_s)


def test_a_bus_whose_exchange_does_not_end_reads_as_silent_and_never_holds_the_cycle_up() -> None:
    # a wedged backend: its drives' replies are missing in that cycle (and while it stays wedged); the other bus
    # answers in every cycle, each cycle ends within WORKER_GRACE_S of its deadline; once it ends, the bus is back
    emulator = Emulator([1, 101])
    channels = [uuid.uuid4().hex, uuid.uuid4().hex]
    with contextlib.ExitStack() as stack:
        for line, channel in enumerate(channels):
            stack.enter_context(VirtualCanAttachment(emulator, channel, line=line))
        stalling = _Stalling("virtual", channels[1], None)
        buses = stack.enter_context(Buses([CanTransport("virtual", channels[0], None), stalling], ["left", "right"]))
        batch = [Request(1, Bare(Command.READ_STATUS_1)), Request(101, Bare(Command.READ_STATUS_1))]
        for _ in range(3):
            deadline = buses.clock() + 0.05
            replies = buses.transact(batch, deadline)
            assert buses.clock() < deadline + WORKER_GRACE_S + 0.05  # (+ this host's scheduling)
            assert [(r.motor_id, r.ok) for r in replies] == [(1, True), (101, False)]
        assert not buses.closed
        _Stalling.release.set()
        time.sleep(0.2)  # (the wedged exchange ends; its late reply is the next one's stale frame)
        for _ in range(3):
            replies = buses.transact(batch, buses.clock() + 0.2)
        assert [(r.motor_id, r.ok) for r in replies] == [(1, True), (101, True)]


def test_the_api_emulates_both_buses_in_real_time_in_a_process_of_their_own(tmp_path: Path) -> None:
    # Arm(emulate="realtime"): `rmd-motion emulate` with a pty per bus, the bus overrides a mapping per bus (at 50 Hz:
    # a rate a busy host holds; the rate check's refusal is a skip)
    try:
        with Arm.from_config(_copy_at(tmp_path, 50), emulate="realtime") as arm:
            assert arm.bus is not None and isinstance(arm.bus, Buses)
            assert [b.describe().split(":")[0] for b in arm.bus.buses] == ["can slcan", "can slcan"]
            arm.move_to({"left_elbow_pitch": 20.0, "right_elbow_pitch": -20.0}, speed_scale=0.5)
            q = arm.positions()
    except RateError as exc:
        pytest.skip(f"this host does not hold bimanual.yaml at 50 Hz just now: {exc}")
    tolerance = BIMANUAL.control.goal_tolerance_deg + 0.01
    assert abs(q["left_elbow_pitch"] - 20.0) < tolerance and abs(q["right_elbow_pitch"] + 20.0) < tolerance


def test_a_simulated_generation_probe_drops_the_outstanding_marks_too() -> None:
    # as CanTransport's (de860ff): the probe drains the late replies the marks wait for; a mark left would swallow
    # the drive's next real answer
    emulator = Emulator([1])
    emulator.add_fault(Fault(InjectedFault.DELAY, 1, start_s=0.0, end_s=0.05, value=30.0))
    simulation = Simulation(emulator)
    bus = SimulatedBus(simulation)
    assert not bus.transact([Request(1, Bare(Command.READ_STATUS_1))], bus.clock() + 0.005)[0].ok
    simulation.sleep_until(simulation.now_s + 0.06)  # the late reply has arrived
    assert bus.probe_families([1], 0.02) == {1: ProtocolFamily.V2}
    (reply,) = bus.transact([Request(1, Bare(Command.READ_STATUS_1))], bus.clock() + 0.01)
    assert reply.ok and bus.counters[1].stale_frames == 0


def test_a_turn_record_belongs_to_the_drive_on_its_bus(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # the record keeps each joint's drive address: a joint moved to the other bus at the same motor id is another
    # drive, whose turns the record does not give
    monkeypatch.setenv("RMD_MOTION_STATE_DIR", str(tmp_path))
    entry = {"turns": 2, "reading_deg": 12.5, "source": "power-on window", "power_on": None}
    document = {
        "schema": TURNS_SCHEMA,
        "version": TURNS_VERSION,
        "bus": "here",
        "joints": {"right_base_yaw": {**entry, "motor_id": 101}, "left_base_yaw": {**entry, "motor_id": 1}},
    }
    turns_store(BIMANUAL).write_text(json.dumps(document))
    assert set(load_turn_records(BIMANUAL, "here")) == {"right_base_yaw", "left_base_yaw"}
    moved = [
        dataclasses.replace(j, bus="left", bus_index=0, motor_id=7) if j.name == "left_base_yaw" else j
        for j in BIMANUAL.joints
    ]
    moved = [dataclasses.replace(j, bus="left", bus_index=0) if j.name == "right_base_yaw" else j for j in moved]
    # right_base_yaw now on the left bus at motor id 1 (its id on the right bus): not the drive the record was made on
    assert set(load_turn_records(dataclasses.replace(BIMANUAL, joints=tuple(moved)), "here")) == set()
