"""An arm whose buses are of both transports, or several RS485 lines (issue 35: "each a full bus section, CAN or
RS485"): bimanual.yaml with its right arm on an RS485 line. One trajectory over both, each bus's exchange at the
same time (the CAN bus's frames at once, the RS485 line's one after the other), each bus's status reads by what its
wire carries, 0x280 on the CAN bus only, and one safety domain."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from motion.api import Arm
from motion.api.emulation import simulated_lines
from motion.config import ArmConfig, ControlMode, load_config
from motion.config.schema import HaltPolicy
from motion.control.ratecheck import RateError
from motion.emulator import Emulator, Rs485Attachment
from motion.emulator.arm import arm_emulator
from motion.emulator.cli import _attachments, _links, add_emulate_arguments
from motion.emulator.faults import Fault, InjectedFault
from motion.emulator.simulated import SimulatedBus, Simulation
from motion.emulator.timing import TimingModel
from motion.protocol import Bare, Command
from motion.safety import ArmState
from motion.transport import Request
from motion.transport.buses import Buses
from tests.motion_rig import Rig, emulated_arm, logged_requests, received
from tests.test_buses import TARGETS, fault_halts_every_axis, setpoint_arrivals
from tests.test_cli import cli, host_stall_misses

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
#: Six V2 drives on an RS485 line at 115200 baud (the older family's fastest) hold a few tens of Hz.
RATE_HZ = 25.0


def _mixed(tmp_path: Path, *, right: str = "rs485", left: str = "can") -> Path:
    """bimanual.yaml (and its URDF) in ``tmp_path`` at :data:`RATE_HZ` with each arm's bus of the transport named,
    a quarter of a second for a reply (the real-time test on a busy host)."""
    shutil.copy(CONFIGS / "bimanual.urdf", tmp_path / "bimanual.urdf")
    data = yaml.safe_load((CONFIGS / "bimanual.yaml").read_text())
    for name, transport in (("left", left), ("right", right)):
        if transport == "rs485":
            data["buses"][name] = {"transport": "rs485", "port": f"/dev/ttyUSB-{name}", "baudrate": 115200}
    data["control"]["rate_hz"] = RATE_HZ
    data["safety"]["reply_timeout_ms"] = 250
    path = tmp_path / "mixed.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _config(tmp_path: Path, **transports: str) -> ArmConfig:
    return load_config(_mixed(tmp_path, **transports))


def _arrivals(rig: Rig, references: list[np.ndarray]) -> list[int]:
    """The cycle at which each joint's reference reached its target for good."""
    reference = np.array(references)
    arrived = [int(np.argmax(np.abs(reference[:, i] - TARGETS[i]) < 1e-9)) for i in range(len(TARGETS))]
    assert all(np.abs(reference[a:, i] - TARGETS[i]).max() < 1e-9 for i, a in enumerate(arrived))
    return arrived


@pytest.mark.parametrize(
    "transports", [{"right": "rs485"}, {"left": "rs485", "right": "rs485"}], ids=["can+rs485", "two rs485"]
)
def test_an_arm_on_a_can_bus_and_an_rs485_line_moves_as_one(tmp_path: Path, transports: dict[str, str]) -> None:
    config = _config(tmp_path, **transports)
    with emulated_arm(config, "sim", tmp_path, supervised=True) as rig:
        supervisor = rig.supervisor
        assert supervisor is not None
        # each bus's status reads by its wire: the RS485 line one a cycle, the CAN bus all twelve of its drives'
        # (each at most 50 ms old at 25 Hz)
        per_cycle = [count for _, count in supervisor.status_rounds.rounds]
        assert per_cycle == [1 if transports.get(side, "can") == "rs485" else 12 for side in ("left", "right")]
        references: list[np.ndarray] = []
        rig.controller.cycle_hooks.append(lambda c, _start, _replies: references.append(c.reference.position.copy()))
        supervisor.move_to(TARGETS, 1.0)
        assert supervisor.wait(30.0)
        arrived = _arrivals(rig, references)
        assert max(arrived) - min(arrived) <= 1 and min(arrived) >= 15, arrived  # (a real move: 0.8 s at 25 Hz)
        np.testing.assert_allclose(
            rig.controller.snapshot.position_deg, TARGETS, atol=config.control.goal_tolerance_deg
        )
    # every drive got its 0xA4 stream on its own bus (the right arm's in RS485 framing on the second line)
    lines: dict[int, set[str]] = {}
    for text in rig.frame_log.read_text().splitlines():
        fields = text.split(maxsplit=3)
        if len(fields) == 4 and fields[1] == "IN":
            lines.setdefault(0 if fields[2].endswith(("can", "rs485")) else 1, set()).add(fields[2])
    assert lines[1] == {"sim-rs485-1"}
    assert set(received(rig, Command.MULTI_TURN_POSITION_SPEED)) == {j.address for j in config.joints}


def test_each_cycle_runs_the_can_bus_and_the_rs485_line_at_the_same_time(tmp_path: Path) -> None:
    # simulated wire time: the CAN bus's six 0xA4 are on their drives long before the RS485 line's last one; the
    # line's last 0xA4 of each cycle reaches its drive within the cycle, not after the CAN bus's batch
    config = _config(tmp_path)
    with emulated_arm(config, "sim", tmp_path, supervised=True) as rig:
        assert rig.supervisor is not None
        rig.supervisor.move_to(TARGETS, 1.0)
        rig.sleep(1.0)
    arrivals = setpoint_arrivals(rig)
    first = {key: min(times) for key, times in arrivals.items()}
    cycles = sorted({cycle for cycle, bus in first if bus == 1 and (cycle, 0) in first})
    assert len(cycles) > 20
    # each cycle's first set-point on each bus goes out at the cycle's start: the line does not wait for the bus
    skew = [abs(first[(c, 1)] - first[(c, 0)]) for c in cycles]
    assert max(skew) < 3e-3, max(skew)  # (one RS485 0xA4 takes 1.6 ms at 115200 baud; a CAN frame 0.13 ms)
    # the line's six, one after the other, all within the cycle; the CAN bus's six long before the line's last
    period = 1.0 / RATE_HZ
    assert all(len(arrivals[(c, 1)]) == 6 and max(arrivals[(c, 1)]) - first[(c, 0)] < period for c in cycles)
    assert all(max(arrivals[(c, 0)]) < max(arrivals[(c, 1)]) - 5e-3 for c in cycles)


def test_torque_mode_sends_0x280_on_the_can_bus_and_0xa1_on_the_rs485_line(tmp_path: Path) -> None:
    config = _config(tmp_path)
    config = dataclasses.replace(config, control=dataclasses.replace(config.control, mode=ControlMode.TORQUE))
    with emulated_arm(config, "sim", tmp_path, supervised=True) as rig:
        # (holding the pose: the example's torque-mode gains are tuned for 250 Hz, not this line's 25 Hz)
        assert rig.supervisor is not None
        rig.sleep(1.0)
        assert rig.supervisor.state is ArmState.READY and not rig.supervisor.faults
    multi = [t for t, address, message in logged_requests(rig) if address is None]
    torque = {
        address for _, address, message in logged_requests(rig) if getattr(message, "command", None) == Command.TORQUE
    }
    assert len(multi) >= RATE_HZ * 0.8  # the CAN bus's motors 1..4: one frame a cycle
    assert torque == {5, 6, 101, 102, 103, 104, 105, 106}  # the left's beyond 4, every drive of the line


@pytest.mark.parametrize(
    ("kind", "address", "value", "limit_c", "expected"),
    [
        # the line's elbow: its temperature in every motion reply, above our limit (the line's 0x9A flags come round
        # once in twelve cycles; the drive's own protection stopping it is seen as a following error before)
        (InjectedFault.OVER_TEMPERATURE, 103, 90.0, 85.0, "temperature"),
        (InjectedFault.SILENT, 105, None, 100.0, "no_reply"),  # the line's wrist_pitch falls silent
        # the CAN bus's shoulder: its drive's flag (0x9A, every drive's each cycle at 25 Hz), our limit above it
        (InjectedFault.OVER_TEMPERATURE, 2, 90.0, 100.0, "drive_over_temperature"),
    ],
)
def test_a_fault_on_either_transport_halts_all_twelve_axes_in_its_detection_cycle(
    tmp_path: Path, kind: InjectedFault, address: int, value: float | None, limit_c: float, expected: str
) -> None:
    config = _config(tmp_path)
    joints = tuple(dataclasses.replace(j, temperature_limit_c=limit_c) for j in config.joints)
    # (the drives' own halt, 0x81, on every fault: what each drive received tells the cycle it was halted in)
    control = dataclasses.replace(config.control, halt_policy=HaltPolicy.STOP)
    safety = dataclasses.replace(config.safety, reply_timeout_ms=20)
    config = dataclasses.replace(config, joints=joints, control=control, safety=safety)
    fault_halts_every_axis(config, tmp_path, kind, address, value, expected, after_s=0.6)


def move_both_elbows(config: Path, *options: str | Path) -> None:
    """``rmd-motion move --emulate`` of both arms' elbows (20 and -20 deg) with ``options``: both arrive."""
    moved = cli("move", "--config", config, "--emulate", *options, "left_elbow_pitch=20", "right_elbow_pitch=-20")
    assert moved.returncode == 0, moved.stderr
    assert "right_elbow_pitch=-20.00" in moved.stdout and "left_elbow_pitch=20.00" in moved.stdout


def test_the_cli_moves_an_arm_on_both_transports_in_simulated_time_and_traces_each_bus_in_its_form(
    tmp_path: Path,
) -> None:
    trace = tmp_path / "run.log"
    move_both_elbows(_mixed(tmp_path), "--trace", trace)
    # the CAN bus's frames as candump lines (their identifiers), the line's as RS485 hex lines, each named by its bus
    lines = [line.split() for line in trace.read_text().splitlines()]
    left = [fields for fields in lines if fields[1] == "left"]
    right = [fields for fields in lines if fields[1] == "right"]
    assert len(left) + len(right) == len(lines) and left and right
    assert any(fields[2].startswith("141#A4") and fields[3] == "T" for fields in left)
    assert all("#" in fields[2] and fields[-1] in ("T", "R") for fields in left)
    assert any(fields[2:5] == ["T", "3E", "A4"] for fields in right)
    assert all(fields[2] in ("T", "R") and fields[3] == "3E" for fields in right)


def test_the_api_emulates_both_transports_in_real_time_on_a_slcan_and_an_rs485_pty(tmp_path: Path) -> None:
    # Arm(emulate="realtime"): `rmd-motion emulate --slcan-link left=... --rs485-link right=...`, the overrides a
    # mapping per bus of each one's keys (the rate check's refusal on a busy host is a skip)
    path = _mixed(tmp_path)
    data = yaml.safe_load(path.read_text())
    data["safety"]["max_missed_replies"] = host_stall_misses(RATE_HZ)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    try:
        with Arm.from_config(path, emulate="realtime") as arm:
            assert arm.bus is not None and isinstance(arm.bus, Buses)
            assert [b.describe().split(" ")[0] for b in arm.bus.buses] == ["can", "rs485"]
            arm.move_to({"left_elbow_pitch": 20.0, "right_elbow_pitch": -20.0}, speed_scale=0.5)
            q = arm.positions()
    except RateError as exc:
        pytest.skip(f"this host does not hold the mixed arm at {RATE_HZ:g} Hz just now: {exc}")
    tolerance = load_config(path).control.goal_tolerance_deg + 0.01
    assert abs(q["left_elbow_pitch"] - 20.0) < tolerance and abs(q["right_elbow_pitch"] + 20.0) < tolerance


def test_each_lines_time_is_its_own_and_a_line_missing_a_reply_took_the_whole_exchange(tmp_path: Path) -> None:
    # what the rate check names the limiting bus by: the RS485 line's six exchanges one after the other take far
    # longer than the CAN bus's six frames at once; a line whose drive is silent took until the deadline
    config = _config(tmp_path)
    emulator, _ = arm_emulator(config)
    simulation = Simulation(emulator, lines=simulated_lines(config))
    reads = [Request(j.address, Bare(Command.READ_STATUS_2)) for j in config.joints]
    with SimulatedBus(simulation, names=("left", "right")) as bus:
        assert all(r.ok for r in bus.transact(reads, simulation.now_s + 0.05))
        healthy = bus.bus_times_s()
        assert healthy is not None and 0.0 < healthy["left"] < 0.002 < healthy["right"] < 0.02, healthy
        now = simulation.now_s
        emulator.add_fault(Fault(InjectedFault.SILENT, 106, start_s=now, end_s=now + 60.0))  # (the line's last)
        replies = bus.transact(reads, now + 0.05)
        whole = simulation.now_s - now  # (the silent drive's share of the cycle, then the rest of the line)
        assert [r.motor_id for r in replies if not r.ok] == [106]
        silent = bus.bus_times_s()
        assert silent is not None and silent["right"] == pytest.approx(whole) and whole > healthy["right"] + 0.005
        assert silent["left"] == pytest.approx(healthy["left"])


def test_the_rate_check_of_an_arm_on_both_transports_names_the_rs485_line(tmp_path: Path) -> None:
    with Arm.from_config(_mixed(tmp_path), emulate=True) as arm:
        check = arm.rate_check
    assert check is not None
    times = dict(check.by_bus_p99_s)
    assert times["right"] > 2 * times["left"] > 0.0, times  # (six exchanges in turn at 115200 baud)
    assert "bus right limits" in check.summary()


def test_the_emulator_times_each_rs485_line_at_its_own_configured_baud_rate(tmp_path: Path) -> None:
    # `rmd-motion emulate --config FILE --bus-time`: each line's frames take the time of its bus's baudrate (the
    # configuration's, by line), unless --baud names one for every line
    parser = argparse.ArgumentParser()
    add_emulate_arguments(parser)
    links = [f"--rs485-link=left={tmp_path / 'l'}", f"--rs485-link=right={tmp_path / 'r'}"]
    buses = [("left", "rs485"), ("right", "rs485")]
    for given, expected in (([], [57600, 115200]), (["--baud", "19200"], [19200, 19200])):
        args = parser.parse_args(["--ids", "1", *links, "--bus-time", *given])
        args.line_bauds = {0: 57600, 1: 115200}
        emulator = Emulator([1, 101])
        with contextlib.ExitStack() as stack:
            made = [
                stack.enter_context(a) for a in _attachments(args, emulator, TimingModel(), None, _links(args, buses))
            ]
            assert [a.baud for a in made if isinstance(a, Rs485Attachment)] == expected
